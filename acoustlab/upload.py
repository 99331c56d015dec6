"""``python -m acoustlab.upload RUN_DIR ...``: send run directories to MLflow after the fact."""

import sys

from acoustlab.tracking import main

if __name__ == "__main__":
    sys.exit(main())
