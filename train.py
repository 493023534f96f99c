"""``python train.py ...`` from a checkout: the same command as ``kpflow-train`` (:mod:`kpflow.cli.train`)."""

from kpflow.cli.train import main

if __name__ == "__main__":
    main()
