"""``python -m harness``: the Hydra app (see ``conf/config.yaml``)."""

from harness.app import main

if __name__ == "__main__":
    main()
