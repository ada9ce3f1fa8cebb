import sys

from zenswarm.compose.cli import main

sys.exit(main())
