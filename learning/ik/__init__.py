"""`felis.learning.ik`."""
