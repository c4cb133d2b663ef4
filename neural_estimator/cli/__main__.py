"""``python -m neural_estimator.cli``: the ``neural-estimator`` command."""

import sys

from neural_estimator.cli.app import main

sys.exit(main())
