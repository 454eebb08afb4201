"""Simulated robosuite tasks, scripted experts and demonstration collection for dyq's closed-loop evaluation."""
