"""Readers for motion files from outside: Vive recordings (csv), BVH and glTF rigs.

Every reader validates what it reads and raises ``FormatError`` naming the file and the
line (or byte offset) of the first problem."""
