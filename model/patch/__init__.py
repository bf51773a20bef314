"""The parameter maps of a patch of skin: the maps, their files and their edits."""
