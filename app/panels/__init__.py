"""One module per GUI panel; each builds its widgets and wires them to the state."""
