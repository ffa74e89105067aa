"""Command-line interface (CONTRACT §3). One module per subcommand, each with ``register``."""
