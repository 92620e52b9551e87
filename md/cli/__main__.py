"""``python -m md.cli ...`` is the ``md`` command."""

import sys

from md.cli import main

if __name__ == "__main__":
    sys.exit(main())
