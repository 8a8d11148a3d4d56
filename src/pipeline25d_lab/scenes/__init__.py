"""Generated scenes with exact truth: the demo city, the rugged city, a CityGML city, an OSGB dataset, bad inputs."""
