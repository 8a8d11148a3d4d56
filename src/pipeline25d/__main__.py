import sys

from pipeline25d.cli import main

sys.exit(main())
