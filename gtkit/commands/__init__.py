"""CLI subcommands, one module each (see gtkit.cli)."""
