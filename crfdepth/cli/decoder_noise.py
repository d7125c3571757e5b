"""What the image decoders' C libraries print on stderr, kept off a command's output: the library's
:mod:`crfdepth.io.decoder_noise`, where the commands' image reading (also the library's, a ROS bag's frames)
finds it."""

from crfdepth.io.decoder_noise import NOISE, quiet_decoders

__all__ = ["NOISE", "quiet_decoders"]
