"""The contract shared by datagen, training, export and service.

Everything that crosses a boundary between those parts is defined here, once:
camera intrinsics (``camera``), the grasp pose vector layout and quaternion
convention (``pose``), crop geometry (``crop``), input normalisation
(``normalization``), the dataset schema (``schema``) and the model card
(``model_card``), and the missing-depth fill (``inpaint``). This package depends on
numpy, Pillow and OpenCV (headless) only, so the service can use it without torch.
"""

__version__ = "0.1.0"
