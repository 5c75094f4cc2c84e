"""Test-session settings, applied before any test module imports numpy.

Importing `tasks` sets its process defaults (one BLAS thread, headless MuJoCo; see
tasks/__init__.py); numpy is not loaded yet when pytest reads this file.
"""

import tasks  # noqa: F401
