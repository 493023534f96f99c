"""The two blocks to stack: a yellow "cheese" block (the one picked) and a larger, flatter green "lettuce" block
(the one it goes onto), both textured so that image features have something to hold on to.

Sizes are half extents (m). The two differ in shape (aspect ratio and height) as well as in colour and texture.
"""

from __future__ import annotations

from typing import Callable

from robosuite.models.objects import BoxObject, MujocoObject
from robosuite.utils.mjcf_utils import CustomMaterial

CHEESE, LETTUCE = "cheese", "lettuce"
SIZES = {CHEESE: (0.045, 0.028, 0.022), LETTUCE: (0.065, 0.05, 0.014)}
_TEXTURES = {CHEESE: "Lemon", LETTUCE: "WoodGreen"}


def _block(name: str) -> MujocoObject:
    material = CustomMaterial(
        texture=_TEXTURES[name],
        tex_name=f"{name}_tex",
        mat_name=f"{name}_mat",
        tex_attrib={"type": "cube"},
        mat_attrib={"texrepeat": "1 1", "specular": "0.2", "shininess": "0.1"},
    )
    return BoxObject(name=name, size=list(SIZES[name]), rgba=None, material=material, density=400)


#: name -> factory of the block
BLOCKS: dict[str, Callable[[], MujocoObject]] = {CHEESE: lambda: _block(CHEESE), LETTUCE: lambda: _block(LETTUCE)}
