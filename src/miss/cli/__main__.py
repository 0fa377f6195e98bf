import sys

from miss.cli import main

sys.exit(main())
