import sys

from afmdrift.cli import main

sys.exit(main())
