import sys

from bayesrob.cli import main

sys.exit(main())
