"""The fusion node (``kmea fuse``) and its benchmark."""
