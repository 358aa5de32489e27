"""Gain tuning of K_GP, K_GI, tau and G_e (issue 4): not built yet."""
