"""``python -m ultratight.receiver.cli``: the ``ultratight`` command."""
import sys

from ultratight.receiver.cli.main import console_main

sys.exit(console_main())
