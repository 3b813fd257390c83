"""Tasks, backend-free (`felis.scenarios`): drops and pushes, and the verdicts on what happened."""
