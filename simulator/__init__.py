"""The seeder in software: device servers on pty pairs plus a plant model with ground truth."""
