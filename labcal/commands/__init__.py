"""One module per command group; each has `register(subparsers)` adding its parser(s)."""
