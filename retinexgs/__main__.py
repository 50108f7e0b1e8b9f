import sys

from retinexgs.cli import main

sys.exit(main())
