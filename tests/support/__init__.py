"""What the tests share: the helpers their modules import (fixtures are in the conftest files).

No test module imports another; each imports from here (``tests/system/test_architecture.py``
holds that).
"""
