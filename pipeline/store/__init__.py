"""The zarr map store: its layout and integrity (``layout``), feature groups (``feature_groups``)
and their compression (``compression``), the reader localization uses (``reader``), and the check
of every chunk (``check``). docs/map_store.md describes the format."""
