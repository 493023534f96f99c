"""``python evaluate.py ...`` from a checkout: the same command as ``kpflow-evaluate`` (:mod:`kpflow.cli.evaluate`)."""

from kpflow.cli.evaluate import main

if __name__ == "__main__":
    main()
