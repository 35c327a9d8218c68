"""Unit conversions. Speeds are m/s inside the simulation; the papers and configs speak km/h."""

KMH = 1.0 / 3.6  # m/s per km/h
