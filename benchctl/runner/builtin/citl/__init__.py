"""Camera in the loop (Peng et al. 2020): the procedure (`procedure`) and its report (`report`)."""
