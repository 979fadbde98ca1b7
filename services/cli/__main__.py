"""``python -m services.cli ARGS...``: ``artrack ARGS...``, the way the launcher starts its processes."""

import sys

from services.cli import main

if __name__ == "__main__":
    sys.exit(main())
