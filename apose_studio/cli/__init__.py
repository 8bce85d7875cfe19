"""The `apose` command line: the parser and most commands (commands), the per-frame commands estimate,
eval and capture checks (frames), and the multi-view ones (views)."""
