"""Help texts as a user reads them."""
from __future__ import annotations

import pytest

from gtkit.cli import build_parser


def test_track_help_keeps_its_usage_lines(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["track", "--help"])
    out = capsys.readouterr().out
    lines = out.splitlines()
    for start in ("gtkit track DIR [--poses FILE]", "gtkit track calibrate DIR ", "gtkit track evaluate DIR "):
        assert any(line.startswith(start) for line in lines), (start, out)
