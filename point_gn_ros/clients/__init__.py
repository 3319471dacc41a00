"""Programs that start the node and talk to it over DDS: the demo and the node benchmark."""
