import os
import sys
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
BRIGHTON = SHARED / "data" / "brighton_beach"
sys.path.insert(0, str(ROOT))
