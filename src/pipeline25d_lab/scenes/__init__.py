"""Generated scenes with exact truth: the demo city, the rugged city, a CityGML city, building-only
cities, an OSGB dataset, bad inputs."""
