"""The commands' configurations: ``overtake-train``'s typed options and each paper's
training recipe as a preset of them."""
