"""facewire: a model-based video call. Its parts: facewire.sender, facewire.receiver,
facewire.protocol and facewire.models (folders at the top of the repository, linked here so
that they install as one package), with the command-line layer in this folder."""
