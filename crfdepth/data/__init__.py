from crfdepth.data.kitti import KittiDepthCompletion, KittiRawScans, KittiTestCompletion, KittiValSelection
from crfdepth.data.sample import Batch, Sample, collate_samples
from crfdepth.data.transforms import BottomCenterCrop, Compose, HorizontalFlip, SubsampleSparse
from crfdepth.data.factory import LAYOUTS, build_dataset
from crfdepth.data.synthetic import SyntheticScenes, make_scene
