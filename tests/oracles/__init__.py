"""Independent oracles that several test modules compare the library against (float64
NumPy, scipy or torch; nothing here calls the code it checks)."""
