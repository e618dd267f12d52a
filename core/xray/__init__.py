"""2D X-ray analysis (stage 3 of DESIGN.md): roadmap vessels, wire segmenters and the ordered wire.

- ``imaging``: shared 2D helpers (input checks, normalisation, polarity, field of view, polyline normals)
- ``unet``: the UNet architecture both networks use
- ``vessels2d_learned``: the learned roadmap vessel mask
- ``wirepresence``: is there a wire in this frame at all
- ``wiremask``: the ordered sub-pixel wire rendered back as a tube
- ``roadmap``: the roadmap's vessel mask (classical vesselness, or the learned one) and its 2D centerline
- ``orderedwire``: the ordered sub-pixel wire (proximal -> distal) traced in a wire mask; the paper's wire graph
- ``segmentation``: the wire segmenters (UNet, ridge), one ``Segmenter`` per ``SegMethod`` in ``SEGMENTERS``
"""
