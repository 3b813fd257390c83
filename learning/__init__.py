"""Learning (`felis.learning`): landing-net evolution, the IK LSTM, phase models. Not built yet."""
