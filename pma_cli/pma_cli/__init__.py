"""The `pma` command line: thin clients over the project's topics, services and actions."""
