"""The registration record (``work/register/registration.json``) read in one place, and each query
sequence's outcome said in words.

``gtkit register`` writes one entry per sequence under ``sequences``; it can be any of
:data:`OUTCOMES`. Every reader (the GT report, ``gtkit register``'s and ``gtkit run``'s lines, the
run summary) goes through :func:`outcome` and :func:`describe`, so a new way of registering a
sequence is taught to them all at once and none of them meets a field it does not expect (an
entry of an older record without ``registered_by`` is a clicked one, as it was then).
"""
from __future__ import annotations

import json
from pathlib import Path

from ..errors import GtkitError

CLICKED = "clicked tie points"
AUTOMATIC = "automatic matches"
SINGLE_PHOTOS = "single photos"
NEEDS_CLICKS = "needs clicks"
ERROR = "error"
OUTCOMES = (CLICKED, AUTOMATIC, SINGLE_PHOTOS, NEEDS_CLICKS, ERROR)


def read_registration(path: str | Path, strict: bool = False) -> dict | None:
    """The record as written (``Paths.registration``), or None where there is none. One that
    cannot be read as JSON is None too, or with ``strict`` a GtkitError naming the file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        if strict:
            raise GtkitError(f"unreadable registration record ({e})", path) from None
        return None
    if not isinstance(data, dict):
        if strict:
            raise GtkitError("unreadable registration record (not a JSON object)", path)
        return None
    return data


def tiepoints(record: dict | None) -> dict[str, dict]:
    """Each clicked tie point's entry (``in_final_ba``, residuals) in the joint adjustment."""
    return dict((record or {}).get("tiepoints") or {})


def bad_tiepoints(record: dict | None) -> dict[str, dict]:
    """The tie points the registration left out as outliers, with why."""
    return dict((record or {}).get("bad_tiepoints") or {})


def sequences(record: dict | None) -> dict[str, dict]:
    return dict((record or {}).get("sequences") or {})


def outcome(s: dict) -> str:
    """One of :data:`OUTCOMES` for a sequence's entry."""
    if s.get("status") != "registered":
        return NEEDS_CLICKS if s.get("needs_clicks") else ERROR
    by = s.get("registered_by") or CLICKED
    if by.startswith(SINGLE_PHOTOS):
        return SINGLE_PHOTOS
    return AUTOMATIC if by == AUTOMATIC else CLICKED


def is_registered(s: dict) -> bool:
    return outcome(s) in (CLICKED, AUTOMATIC, SINGLE_PHOTOS)


def _num(v, nd: int = 3, unit: str = "") -> str:
    if isinstance(v, int) and not isinstance(v, bool):
        return f"{v}{unit}"
    return "–" if v is None else (f"{v:.{nd}f}{unit}" if isinstance(v, float) else str(v))


def _left_out(s: dict) -> tuple[int, int, list[str]]:
    """Photos the sequence's SfM left out: (resected, of how many, 'name (why)' of those not placed)."""
    res = s.get("left_out_by_sfm") or {}
    done = sum(1 for r in res.values() if r.get("resected"))
    why = [f"{n.split('/')[-1]} ({r.get('auto_reason') or r.get('reason') or 'not placed'})"
           for n, r in res.items() if not r.get("resected")]
    return done, len(res), why


def short(s: dict) -> str:
    """A few words: how the sequence was placed, or that it was not (for one-line summaries)."""
    o = outcome(s)
    if o == SINGLE_PHOTOS:
        done, n, _ = _left_out(s)
        return f"single photos (its SfM made no model): {done} of {n} photos placed one by one"
    return {CLICKED: "clicked tie points", AUTOMATIC: "automatic matches (no usable clicks)",
            NEEDS_CLICKS: "not registered: needs clicks", ERROR: "not registered"}[o]


def describe(s: dict) -> str:
    """The sequence's outcome in one sentence with its figures (the GT report's and
    ``gtkit register``'s line)."""
    o = outcome(s)
    if o in (NEEDS_CLICKS, ERROR):
        return f"not registered{' (needs clicks)' if o == NEEDS_CLICKS else ''}: {s.get('error') or 'no reason recorded'}"
    final = s.get("n_tiepoints_final_ba")
    if o == SINGLE_PHOTOS:
        done, n, why = _left_out(s)
        text = (f"registered as single photos (its SfM made no model): {done} of {n} photos placed one by one "
                "from automatic matches to the reference")
        return text + (f"; not placed: {', '.join(why)}" if why else "")
    if o == AUTOMATIC:
        a = s.get("automatic") or {}
        text = (f"registered by automatic matches ({s.get('clicks') or 'no clicks'}); "
                f"{a.get('n_photos_agreeing', '–')}/{a.get('n_photos', '–')} photos agree, "
                f"{a.get('n_sim3_inliers', '–')}/{a.get('n_point_pairs', '–')} block-reference point pairs Sim(3) "
                f"inliers, Sim(3) from {a.get('sim3_from') or '–'}; {_num(final)} clicked tie points in the final BA")
    else:
        text = (f"registered by clicked tie points; {_num(s.get('n_sim3_inliers'))}/{_num(s.get('n_tiepoints'))} "
                f"tie points Sim(3) inliers, {_num(final)} in the final BA, Sim(3) RMSE {_num(s.get('sim3_rmse_m'), unit=' m')}")
    done, n, why = _left_out(s)
    if n:
        text += f"; {done} of {n} photos its SfM left out placed on their own" + (f" (not: {', '.join(why)})" if why else "")
    return text + calibration_words(s)


def calibration_words(s: dict) -> str:
    """'; camera: where its intrinsics came from' for a sequence's entry ('' in an older record)."""
    c = s.get("calibration") or {}
    if not c:
        return ""
    words = f"; camera: {c['source']}"
    if c["source"] == "self-calibrated":
        words = "; camera: " + (c["start"] + ", not confirmed by the ties" if "start" in c else
                                f"self-calibrated from its own {c.get('n_photos', '–')} photos")
        words += " (the last resort"
        words += f": {c['why_not_from_reference']})" if c.get("why_not_from_reference") else ")"
    return words


def counts(record_sequences: dict[str, dict]) -> dict[str, int]:
    """How many sequences had each outcome."""
    out = dict.fromkeys(OUTCOMES, 0)
    for s in record_sequences.values():
        out[outcome(s)] += 1
    return out
