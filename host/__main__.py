import sys

from stereopath.host.cli import main

sys.exit(main())
