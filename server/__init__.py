"""The asyncio websockets server that solves and broadcasts avatars."""
