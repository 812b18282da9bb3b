"""Methods of the matrix: each paper's method as parts in slots (filter engine, motion and observation
models, fusion, learner) that estimate the targets' positions on any scenario they fit."""
