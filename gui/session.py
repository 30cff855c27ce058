"""The annotator's UI state (which pair, which view, which tab), so reopening resumes the work:
``work/annotate/session.json``, written atomically. Tie points themselves live in
``tiepoints.json``, never here."""
from __future__ import annotations

import json
from pathlib import Path

from gtkit.io.atomic import write_json


def session_path(paths) -> Path:
    return paths.stage("annotate") / "session.json"


def load_session(paths) -> dict:
    p = session_path(paths)
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
        return d if isinstance(d, dict) else {}
    except (OSError, json.JSONDecodeError):
        return {}


def save_session(paths, state: dict) -> None:
    write_json(session_path(paths), state)
