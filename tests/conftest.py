"""Suite-wide settings.

Under CI (``CI`` set, as ``.ci/run`` is run) hypothesis draws the same examples on every run, so a
submission lands or fails on its code, not on the draw; locally each run explores new examples, and a
failure found there is pinned with ``@example`` before it is fixed.
"""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
