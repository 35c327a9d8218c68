"""The commands' one door: each mistake at a command's edge gets one line."""
