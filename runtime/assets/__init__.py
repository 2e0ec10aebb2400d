"""What the virtual object is: built-in and user meshes (``objects``) and trained/precomputed object
bundles (``bundle``)."""
