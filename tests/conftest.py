"""The suite's fixtures, each in the support module of what it provides (pytest plugins).

tests/support/s3.py: the SeaweedFS S3 server; cluster.py: the session's Ray; datasets.py: the
datasets made on it; serve_app.py: the links Serve app; browser.py: Chromium; markers.py: the
`ray`, `s3` and `browser` marks set from the fixtures a test uses; needs.py: a missing test
dependency fails a CI run and is a skip elsewhere; workers.py: what keeps two xdist workers
(tests/run's -n 2) apart. tests/engine/conftest.py gives the engine's tests a dataset made
without Ray (the engine's tests run with Ray blocked: tests/run).
"""

pytest_plugins = [
    "tests.support.needs",
    "tests.support.markers",
    "tests.support.s3",
    "tests.support.cluster",
    "tests.support.datasets",
    "tests.support.serve_app",
    "tests.support.browser",
    "tests.support.workers",
]
