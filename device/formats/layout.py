"""Names of the files of our recording layout, shared by the writer and the readers.

A stereopath session is a directory::

    SESSION/
      manifest.json        session id, software version, configuration, rig name, counts, status
      groundtruth.tum      T_world_cam0 ground truth (simulated sessions; written atomically)
      trajectory.tum       the estimated T_world_cam0 path, appended while recording
      mav0/                EuRoC/ASL layout, readable by ORB-SLAM3, OpenVINS, Basalt and Kalibr
        rig.yaml           our full rig calibration (stereopath.device.formats.rig_files.save_rig_yaml; wins over sensor.yaml)
        body.yaml
        cam0/sensor.yaml   EuRoC camera sensor file (T_BS = T_body_cam0, pinhole, radial-tangential)
        cam0/data.csv      "#timestamp [ns],filename"
        cam0/data/<t_ns>.png   lossless 8-bit PNG, mid-exposure time on the session's clock
        cam1/...           the same for the right camera (same t_ns as cam0: frames are pairs)
        imu0/sensor.yaml   EuRoC IMU sensor file (T_BS = identity: the body frame is the IMU frame)
        imu0/data.csv      EuRoC IMU rows (gyro rad/s, specific force m/s^2, body frame)
        imu0/temperature.csv   "#timestamp [ns],temperature [degC]" (only when the IMU reports it)

Ground-truth file names tell their frame apart: ``groundtruth.tum`` (ours) holds camera-0
poses; ``groundtruth_tum.txt`` (the EuRoC convention beside ``mav0``) holds body poses.
"""

from __future__ import annotations

MAV0 = "mav0"
CAMERAS = ("cam0", "cam1")
IMU = "imu0"
RIG_YAML = "rig.yaml"  # inside mav0/
MANIFEST = "manifest.json"
GROUNDTRUTH = "groundtruth.tum"  # T_world_cam0
TRAJECTORY = "trajectory.tum"  # estimated T_world_cam0
EUROC_GROUNDTRUTH_TUM = "groundtruth_tum.txt"  # EuRoC body poses beside mav0
EUROC_GROUNDTRUTH_CSV = "state_groundtruth_estimate0/data.csv"  # EuRoC body poses inside mav0
MOCAP_GROUNDTRUTH_CSV = "mocap0/data.csv"  # TUM VI motion-capture poses of the IMU inside mav0
IMU_TEMPERATURE = "temperature.csv"

CAM_CSV_HEADER = "#timestamp [ns],filename\n"
IMU_CSV_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n"
)
TEMP_CSV_HEADER = "#timestamp [ns],temperature [degC]\n"
TRAJECTORY_HEADER = "# timestamp tx ty tz qx qy qz qw (T_world_cam0, metres, seconds)\n"

FORMAT_NAME = "stereopath-session"
FORMAT_VERSION = 1
