"""``python -m kf_train.cli``: the ``kf-train`` command."""

import sys

from kf_train.cli.dispatch import main

sys.exit(main())
