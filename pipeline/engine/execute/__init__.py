"""Running a plan's tasks: one function for one task (:mod:`.node`), two executors behind one interface
(:mod:`.in_process`, :mod:`.dask_cluster`), and the batch that picks one (:mod:`.batch`).

Kept empty of imports: :mod:`.early_child` is imported by ``polyvec``'s launcher before anything else.
"""
