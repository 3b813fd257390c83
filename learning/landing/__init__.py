"""`felis.learning.landing`."""
