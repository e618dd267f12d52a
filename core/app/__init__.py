"""The application layer: whole runs, outputs, servers and the command line.

- ``pipeline``: ``run`` / ``run_to_outdir``, one case from files to a staged output folder
- ``export``, ``outdir``: writing and reading back the output folder
- ``biplane``: joint registration and two-view frames
- ``stream``: ``guidewire3d live`` (the processing loop, its setup and the command)
- ``sources``: the live frames in (video, folder, DICOM replay) and the one-slot mailbox
- ``igtl``: OpenIGTLink: the messages of a frame, the server and the client (``WireFollower``)
- ``batch``, ``dicomnet``: many studies on Dask; the DICOM C-STORE receiver
- ``batch2d``: ``guidewire3d segment`` on image files
- ``vesselplan``: ``guidewire3d vessels`` (the CTA-only planning command)
- ``bench``: the ``demo`` and ``bench`` commands
- ``cli``: the command line (a front end; it imports each command's modules when the command runs)
"""
