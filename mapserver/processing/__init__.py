"""A log through the engine, the store and the merge.

``run`` (the engine alone), ``live`` (a session merging as it runs), ``pipeline`` (a log into the store,
resumable), ``reckoning`` (dead reckoning of the log's odometry).
"""
