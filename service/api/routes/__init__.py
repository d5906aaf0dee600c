"""The HTTP routes, one module a resource; each parses, calls the engine, shapes the answer."""
