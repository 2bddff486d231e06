"""Operator GUI (PySide6 + pyqtgraph); imports Qt, so nothing outside velab.gui imports it."""
