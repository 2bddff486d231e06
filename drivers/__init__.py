"""Device drivers (Qt-free): one class per device kind, transport injected."""
