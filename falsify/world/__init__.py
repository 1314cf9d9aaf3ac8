"""The world: the modification space and everything a scene is built from (streets, terrain,
vegetation, buildings, road users, cars, materials). Nothing here knows about sensors."""
