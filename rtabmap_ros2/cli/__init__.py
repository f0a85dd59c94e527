"""The ``rtabmap-ros2`` command line: ``cli.py`` (entry point), ``common_args.py`` (parameter options), one ``cmd_<name>.py`` per subcommand."""
