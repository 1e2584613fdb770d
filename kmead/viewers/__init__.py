"""Exports for viewers: Foxglove WebSocket, MCAP."""
