"""What was measured about a bench and how it applies: the calibration store per profile (`store`), its files
checked as they are read (`files`), the acceptance test a new calibration passes before it replaces one
(`acceptance`), each channel's optical setup (`setups`), profiles on other grids (`geometry`)."""
