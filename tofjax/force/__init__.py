"""Force estimation from ToF histograms (seed 001): data, features, models, residual forest, runs."""
