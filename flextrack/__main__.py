import sys

from flextrack.cli import main

sys.exit(main())
