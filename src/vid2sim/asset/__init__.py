"""The asset format: what the reconstruction writes and the simulator reads (docs/asset-format.md)."""

from vid2sim.asset.folder import Asset, AssetFormatError, load_asset, save_asset

__all__ = ["Asset", "AssetFormatError", "load_asset", "save_asset"]
