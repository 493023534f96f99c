"""Tasks: scenes, demonstrators and datasets that produce demonstrations to transport."""
