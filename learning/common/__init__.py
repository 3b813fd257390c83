"""`felis.learning.common`."""
