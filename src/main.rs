fn main() {
    println!("invaders: see README.md");
}
