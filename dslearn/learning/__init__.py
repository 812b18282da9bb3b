"""Learning: GP backends, LSTM training, online EM, factor-graph identification, GP experts."""
