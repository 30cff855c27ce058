import os
import sys
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
BRIGHTON = SHARED / "data" / "brighton_beach"
sys.path.insert(0, str(ROOT))

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def small_sample(tmp_path_factory):
    """The small sample project, generated once per test session (``gtkit sample create``).

    Tests must treat it as read-only; copy it (or use ``sample_copy``) before running stages
    that write into it.
    """
    from gtkit.cli import main

    given = os.environ.get("GTKIT_SMALL_SAMPLE")  # developers: reuse a sample generated before
    if given:
        return Path(given)
    root = tmp_path_factory.mktemp("sample") / "small"
    assert main(["sample", "create", str(root), "--preset", "small", "--seed", "0"]) == 0
    return root


@pytest.fixture(scope="session")
def tiny_sample(tmp_path_factory):
    """The ``tiny`` sample preset (tests only), generated once per session: (root, settings, summary).
    Read-only by convention, like ``small_sample``."""
    from gtkit.synth.generate import create_sample
    from gtkit.synth.settings import load_preset

    root = tmp_path_factory.mktemp("tiny") / "site"
    settings = load_preset("tiny")
    return root, settings, create_sample(root, settings, quiet=True)
