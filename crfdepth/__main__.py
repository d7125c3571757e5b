import sys

from crfdepth.cli import main

sys.exit(main())
