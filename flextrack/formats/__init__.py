"""Readers and writers for the standard formats a sequence folder is made of.

A sequence folder (see DESIGN.md) is readable by BOP and EuRoC tools alike:

    imu0/data.csv          EuRoC ASL IMU csv (ns, rad/s, m/s^2)
    imu0/sensor.yaml       Kalibr IMU noise model (+ T_BS)
    frame_times.csv        `#frame_id,timestamp [ns]`: capture time of every frame
    scene_camera.json      BOP: cam_K per frame
    scene_gt.json          BOP: cam_R_m2c (row-major), cam_t_m2c (mm) per frame
    groundtruth.csv        EuRoC state_groundtruth_estimate0 at the IMU rate
    rig.yaml               T_BC (camera -> IMU body), T_WO (object -> world), object id
    models/                the object's BOP model (.ply in mm, models_info.json)
    rgb/ mask/ depth/      optional rendered frames, named %06d.png by frame id
"""
