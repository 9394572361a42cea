"""One module per `vfdata` subcommand; each defines `register(subparsers)`."""
