//! Goodrive (GD20, GD300, GD10) drive model.
