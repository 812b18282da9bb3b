"""Factor-graph Gaussian message passing for model identification (messages, iterated
identification, CRLB, centralised baselines) and its Monte Carlo engine."""
