"""Sub-commands of the mi-neurallens CLI, one module each."""
