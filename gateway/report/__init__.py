"""``sowgate report``: the field report a farmer keeps (HTML or PDF from the record store).

An application-level command beside ``gateway.app``: it reads the recording domain's store and
draws with matplotlib, which nothing in the daemon imports.
"""
