"""Command-line interface (docs/conventions.md): one module per subcommand, each with
``register``."""
