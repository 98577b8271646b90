from rtupoll.cli import main

main()
