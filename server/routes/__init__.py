"""REST and websocket routes of the live service, one module per resource."""
