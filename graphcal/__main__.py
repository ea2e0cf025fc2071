import sys

from graphcal.cli import main

sys.exit(main())
