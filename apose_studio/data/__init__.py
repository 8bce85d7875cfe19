"""Frames on disk: apose datasets and captures (dataset), BOP scenes and results files (bop), and the
journalled output folders renders write into (outdir)."""
