"""A Griffe extension for the API reference: kpflow's docstrings cross-reference with Sphinx roles
(:class:`~kpflow.maps.base.TransportMap`, :func:`transport_trajectory`, :mod:`.geometry`), which Markdown would show
as literal text. Each role becomes an optional mkdocs-autorefs link: a link where the target is documented on the
site, plain code where it is not (an optional reference never fails ``mkdocs build --strict``).

Names resolve as the docstrings mean them: a dotted ``kpflow.`` path as written, a leading dot as a relative import
(``.scene`` beside the module), anything else through the object's scope (its members, its module's imports, its
parents).
"""

from __future__ import annotations

import html
import re

import griffe

ROLE = re.compile(r":(?:py:)?(class|func|meth|mod|attr|data|obj|exc|const):`(?P<body>[^`]+)`")


def _module_of(obj: griffe.Object) -> griffe.Object:
    while not obj.is_module:
        obj = obj.parent
    return obj


def _resolve(obj: griffe.Object, target: str) -> str:
    if target.startswith("kpflow.") or target == "kpflow":
        return target
    if target.startswith("."):  # as a relative import: ``.scene`` is a sibling module, ``..maps`` one level up
        module = _module_of(obj)
        package = module.path if module.is_init_module else module.path.rpartition(".")[0]
        dots = len(target) - len(target.lstrip("."))
        for _ in range(dots - 1):
            package = package.rpartition(".")[0]
        return f"{package}.{target.lstrip('.')}"
    head, _, rest = target.partition(".")
    try:
        resolved = obj.resolve(head)
    except Exception:  # unresolvable names stay plain code
        return target
    return f"{resolved}.{rest}" if rest else resolved


def rewrite(obj: griffe.Object, text: str) -> str:
    """The docstring ``text`` of ``obj`` with its Sphinx roles turned into optional cross-references."""

    def link(match: re.Match) -> str:
        body = match["body"].strip()
        title, angle = re.match(r"^(.*?)\s*(?:<([^>]+)>)?$", body).groups()  # :class:`title <target>`
        target = (angle or title).lstrip("~!")
        shown = title if angle else (target.rsplit(".", 1)[-1] if title.startswith("~") else target.lstrip("."))
        identifier = _resolve(obj, target)
        return f'<autoref identifier="{html.escape(identifier)}" optional><code>{html.escape(shown)}</code></autoref>'

    return ROLE.sub(link, text)


class SphinxRoles(griffe.Extension):
    """Rewrite every docstring of a loaded package once it is complete (so that names resolve)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        stack = [pkg]
        while stack:
            obj = stack.pop()
            if obj.docstring is not None:
                obj.docstring.value = rewrite(obj, obj.docstring.value)
            stack.extend(member for member in obj.members.values() if not member.is_alias)
