"""Environment variables the mission runner reads, named once. No imports: the command line
names them in its help without loading the bus that reads them."""

#: Where a key comes from when neither ``--bus-key-file`` nor ``bus.auth.key_file`` names one.
DEFAULT_KEY_ENV = "MISSION_BUS_KEY"
#: A process's broker login, over its role's line of the credentials file.
USERNAME_ENV = "MISSION_BUS_USERNAME"
PASSWORD_ENV = "MISSION_BUS_PASSWORD"
