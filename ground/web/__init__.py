"""The live web view of the ground station (`python -m ground.station`): per box, the plots, state and events
(`boxview`), the fleet of boxes (`fleet`), the aiohttp server (`server`) and its page (`static/`)."""
