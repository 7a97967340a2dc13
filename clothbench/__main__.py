import sys

from clothbench.cli import main

sys.exit(main())
