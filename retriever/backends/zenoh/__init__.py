"""The real-time backend over Eclipse Zenoh (DESIGN.md §5, §7). So far: its wire format."""
