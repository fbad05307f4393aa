"""``python -m mipslam ...``: the same command line as the ``mipslam`` console script."""
import sys

from mipslam.cli import main

sys.exit(main())
