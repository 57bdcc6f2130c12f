"""saft: shape and appearance of fabrics from one RGB video and a template mesh.

Data flows one way: Scene (saft.scene) → texture, shape and appearance phases (saft.reconstruct,
saft.appearance) → Result → evaluation and export (saft.evaluate, saft.export).
"""

__version__ = "0.1.0"
