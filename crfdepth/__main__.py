"""``python -m crfdepth``: the ``crfdepth`` command (:func:`crfdepth.cli.main`)."""

import sys

from crfdepth.cli import main

if __name__ == "__main__":
    sys.exit(main())
