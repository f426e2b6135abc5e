import os
import tempfile

# Generated kernels go to a per-run cache unless the caller set one (CI reuses nothing stale).
os.environ.setdefault("ARDFLOW_CACHE_DIR", os.path.join(tempfile.gettempdir(), "ardflow-test-kernels"))
