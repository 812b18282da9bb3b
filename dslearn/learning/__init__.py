"""Learning procedures: the learn-while-tracking loop, online EM, factor-graph identification, LSTM training,
social-force fitting (the models they learn are :mod:`dslearn.models`)."""
