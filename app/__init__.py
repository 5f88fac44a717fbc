"""The factorydet browser app (viser): it draws, routes events and calls factorydet_core."""
