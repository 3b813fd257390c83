"""The ``felis`` command (`felis.cli.main`): wires backends, controllers and learning together."""
