import sys

from mjxdiff.cli import main

sys.exit(main())
