"""What to do about the usual camera problems: one wording, shared by the ptp and gphoto2 drivers and discovery."""

UDEV_RULE = "udev/70-benchctl-canon.rules"
NOT_FOUND_HINT = ("is it on, in PTP mode, not grabbed by a desktop daemon "
                  "(gvfs-gphoto2-volume-monitor)?")
USB_GRABBED_HINT = ("probably a desktop daemon (gvfs-gphoto2-volume-monitor) or another gphoto2: stop it "
                    "(systemctl --user stop gvfs-gphoto2-volume-monitor) and reconnect the camera")
PERMISSION_HINT = (f"install {UDEV_RULE} (sudo cp {UDEV_RULE} /etc/udev/rules.d/ && sudo udevadm control "
                   f"--reload-rules && sudo udevadm trigger), join the plugdev group and reconnect the camera")
NO_FOCUS_HINT = ("the camera could not focus and did not release the shutter: switch the lens or body to manual "
                 "focus (MF) and focus on the image plane by hand")
BUSY_HINT = ("it may still be saving the previous frame or hunting for focus: wait, set manual focus (MF), "
             "and check that no other program talks to the camera")
RAW_HINT = "set the image quality to RAW on the camera"
