"""`felis.learning.balance`."""
