"""The fusion node (``kmea fuse``). Its benchmarks are in :mod:`kmead.benchmarks`
(``kmea bench fusion-node``, ``kmea bench fusion-zenoh``)."""
