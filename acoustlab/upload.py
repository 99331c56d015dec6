"""``python -m acoustlab.upload RUN_DIR ...``: send run directories to MLflow after the fact (see ``acoustlab.run.upload``)."""

import sys

from acoustlab.run.upload import main

if __name__ == "__main__":
    sys.exit(main())
