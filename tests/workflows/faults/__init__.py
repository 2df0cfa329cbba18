"""The fault catalogue: bad inputs and faults, each with the outcome a user gets, by class.

    test_inputs.py         images, cameras, names, query lists (one reader each)
    test_stores.py         missing or damaged store files, incremental maps, --overwrite, the build lock
    test_results.py        results tied to their map, one record per query, priors and ground truth by name
    test_writes.py         atomic outputs, damaged job and shard files, folders that are not ours
    test_messages.py       what a user reads: errors with their fix, dry runs, Ctrl-C, units
    test_random_damage.py  the property behind them: random damage gives a named error or a right result
    test_earlier_cases.py  the cases of earlier rounds (truncated images, damaged chunks, NaN-free summaries)

Every case runs real parts on real data (``../shared``) and says, in its docstring, what happened
before it was fixed.
"""
