"""Fleet reprocessing: many recorded sessions as tasks on Ray (local or a cluster).

:mod:`.sessions` finds sessions and their ids and maps paths for cluster workers;
:mod:`.worker` is what runs inside a Ray worker (one session through the one-session
pipeline, progress reported to a small actor); :mod:`.runner` starts or joins Ray and schedules
the sessions; :mod:`.summary` writes ``fleet.json`` and ``fleet.html``; :mod:`.progress` is the
terminal display; :mod:`.compare` checks two output folders hold the same results.
Ray is imported only by :mod:`.runner` and :mod:`.worker`, inside functions.
"""
