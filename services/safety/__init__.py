"""The emergency-brake supervisor (``racecav safety``): iTTC per lidar ray, brake input of the mux."""
