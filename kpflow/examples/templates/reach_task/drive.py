"""Run reach episodes with the policy a server serves: ``python drive.py [--uri ws://127.0.0.1:8000] [--episodes 5]``.

The robot side of a deployment: the env observes, a :class:`~kpflow.serving.client.PolicyClient` asks the server
for actions, the same closed loop as in-process evaluation runs them (kpflow.core.rollout).
"""

import argparse

from reach import ReachTask

from kpflow.core.rollout import rollout
from kpflow.serving.client import PolicyClient


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--uri", default="ws://127.0.0.1:8000")
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--condition", default="wide")
    parser.add_argument("--wait", type=float, default=60.0, help="seconds to wait for the server")
    args = parser.parse_args()
    client = PolicyClient(args.uri, wait=args.wait)
    task = ReachTask()
    env = task.make_env(args.condition)
    with client:
        wins = sum(
            rollout(env, client, task.max_steps, 2_000_000 + i, {"seed": 2_000_000 + i}).success
            for i in range(args.episodes)
        )
    print(f"{wins}/{args.episodes} episodes reached the target through {args.uri}")
    if not wins:
        raise SystemExit("no episode reached the target: is the server serving a reach policy?")


if __name__ == "__main__":
    main()
