"""Disparity: the matcher settings (config), the matchers built from them (matchers: bm, sgbm;
dense), and fixed-point disparity maps to float pixels (disparity)."""
