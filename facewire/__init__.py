"""facewire: the command-line layer over sender and receiver."""
