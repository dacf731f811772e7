import atexit
import os
import shutil
import sys
import tempfile

sys.path.insert(0, os.path.dirname(__file__))

# The twin cache (fbgcomp.structure.cache) of the test session: a fresh folder, removed at exit,
# so tests never read nor write the user's cache (~/.cache/fbgcomp) and start cold. Subprocesses
# (CLI tests) inherit it.
_TWIN_CACHE_DIR = tempfile.mkdtemp(prefix="fbgcomp-test-cache-")
os.environ["FBGCOMP_CACHE_DIR"] = _TWIN_CACHE_DIR
atexit.register(shutil.rmtree, _TWIN_CACHE_DIR, ignore_errors=True)
