"""Make this checkout's gdiff importable in rule scripts (also inside a rule's conda env)."""
import sys
from pathlib import Path

_root = str(Path(__file__).resolve().parents[2])
if _root not in sys.path:
    sys.path.insert(0, _root)
