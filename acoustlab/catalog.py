"""``python -m acoustlab.catalog``: regenerate docs/features.md (see ``acoustlab.run.catalog``)."""

from acoustlab.run.catalog import main

if __name__ == "__main__":
    main()
