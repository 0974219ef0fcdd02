"""The stages of the reconstruction, one module each (docs/architecture.md)."""
