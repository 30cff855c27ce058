"""``gtkit meta PHOTO...``: print what gtkit reads from photos (EXIF GPS, DJI XMP angles)."""
from __future__ import annotations

import json


def register(sub):
    p = sub.add_parser("meta", help="print EXIF GPS and DJI XMP attitude of photos")
    p.add_argument("photos", nargs="+")
    p.add_argument("--require", choices=["gps", "gimbal"], action="append", default=[])
    p.set_defaults(func=run, writes=False)


def run(args):
    from ..io.exif import read_photo_meta

    for f in args.photos:
        m = read_photo_meta(f, require=tuple(args.require))
        print(json.dumps({"file": f, **{k: v for k, v in m.as_dict().items() if v is not None}}))
