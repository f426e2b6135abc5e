import os
import tempfile

# Generated kernels go to a temp cache unless the caller set one; files are keyed by structure hash and generator version.
os.environ.setdefault("ARDFLOW_CACHE_DIR", os.path.join(tempfile.gettempdir(), "ardflow-test-kernels"))
