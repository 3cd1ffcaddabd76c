"""``python -m sg_torchrl.train``: same as the ``sg-train`` console script."""

import sys

from sg_torchrl.train import main

sys.exit(main())
