"""The real-time backend over Eclipse Zenoh (DESIGN.md §5, §7). So far: its wire format (wire.py) and
its sessions (hub.py); the runtime itself is the next step."""
