"""``python -m ultratight.receiver.cli``: the ``ultratight`` command."""
import sys

from ultratight.receiver.cli.main import main

sys.exit(main())
