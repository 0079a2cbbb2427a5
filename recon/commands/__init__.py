"""``recon`` subcommands, one module each (see :mod:`sonarsim.cli_common`)."""
