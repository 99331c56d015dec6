"""``python -m acoustlab.report PATHS ...``: a Markdown and HTML report of runs (see ``acoustlab.reporting.report``)."""

import sys

from acoustlab.reporting.report import main

if __name__ == "__main__":
    sys.exit(main())
