"""The command-line interfaces of ``hmodel``: one module per subcommand, the options they share."""
