"""Public roadside datasets in (issue 50): readers of the formats real roadside sensors' data is
published in, into one model (`model.RoadsideDataset`: the site's sensors from the dataset's
calibration, frames of files, labels in the site frame) and from it the project's scene
(`site.site_scene`: no lanes needed) and the MEC's bus messages.

    pcd.py        PCD point clouds (ascii, binary, binary_compressed) through open3d's tensor reader
    model.py      the common model, the typed errors, vehicle categories
    openlabel.py  ASAM OpenLABEL 1.0 as TUMTraf / A9 write it (lidar labels, cameras, transforms)
    rope3d.py     Rope3D: KITTI-style camera labels on a ground plane (`denorm`)
    site.py       a dataset's site as the project's scene; its frames as the MEC's messages
"""
