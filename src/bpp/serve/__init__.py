"""Serving policies to robots: ``bpp serve`` (openpi's websocket protocol) and its robot-side client."""
