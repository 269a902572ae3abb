"""The animation pipeline: an animation's frames rendered into a folder (``animation``:
:func:`render_animation`, the ``hlbvh render`` verb), one frame applied, updated,
rendered and timed (``frame``), the settings a render runs with (``settings``), the
output folder (``output``), images written atomically (``images``) and frames rendered
on Dask workers (``cluster``)."""
