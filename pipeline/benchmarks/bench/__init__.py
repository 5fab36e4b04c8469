"""`relight bench`: every relighting method over its parameter sweep, against the reference.

    methods.py     the adapter protocol and the registry of methods (one line per method)
    references.py  reference renders, once per (scene, light edit, bounce count), cached on disk
    measure.py     relighting a cache under every light edit: PSNR, relMSE, relight ms -> SweepRows
    direct.py, transfer.py, gather.py   the adapters of the methods of those names
"""
