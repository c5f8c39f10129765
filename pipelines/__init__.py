"""Thin stages: read artifacts, call the library, write artifacts. Reached from conf/stage/*.yaml."""
