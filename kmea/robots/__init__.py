"""Robots: poses from their markers, the IIR and tracking filters, multi-camera fusion."""
