"""``python -m harness.report SWEEP_DIR`` (see ``harness/report/__init__.py``)."""

import sys

from harness.report import main

if __name__ == "__main__":
    sys.exit(main())
