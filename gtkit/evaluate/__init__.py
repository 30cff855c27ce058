"""Evaluation against truth/. The only package (with the sample generator) that reads truth/."""
