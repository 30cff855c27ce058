"""``python -m gui DIR [--poses FILE] [--query NAME]``: the annotator without the gtkit CLI."""
import argparse
import sys

from .app import main

p = argparse.ArgumentParser(prog="python -m gui")
p.add_argument("project")
p.add_argument("--poses")
p.add_argument("--query")
a = p.parse_args()
sys.exit(main(a.project, a.poses, a.query))
