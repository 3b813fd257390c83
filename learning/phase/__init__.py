"""`felis.learning.phase`."""
