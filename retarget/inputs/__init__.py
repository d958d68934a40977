"""Readers and bodies: capture files (AMASS, OMOMO, BVH, our demonstration ``.npz``) to a
``Demonstration`` (world z-up, metres, wxyz), the human surface, object meshes and the shape
library. Imports nothing else of ``retarget``."""
